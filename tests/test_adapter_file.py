"""The adapter file format v1 (docs/conventions.md section 4): sizes, atomic save, validated load."""

from __future__ import annotations

import json
import os

import pytest
import torch
from safetensors.torch import load_file, save_file

import raytun3r_plugin as rt
from raytun3r_plugin.adapter import COMPONENTS
from raytun3r_plugin.apps.adapter_report import describe_file
from raytun3r_plugin.errors import AdapterError, Raytun3rError
from tests.helpers import fisheye, randomise_

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_network, build_tiny_network  # noqa: E402


@pytest.fixture(scope="module")
def net():
    return build_tiny_network(seed=0)


@pytest.fixture
def saved(net, tmp_path):
    adapter = randomise_(rt.Adapter.for_model(net, fisheye()))
    adapter.training_info = {"steps": 3, "final": {"reproj": 0.5}}
    return adapter, adapter.save(tmp_path / "a.safetensors")


def test_da3_small_has_the_documented_size():
    adapter = rt.Adapter.for_model(build_network("da3-small"))
    assert adapter.backbone == "da3-small"
    assert adapter.num_parameters() == {"pe": 10_752, "rope": 20, "total": 10_772}
    assert adapter.is_zero()


def test_file_holds_exactly_the_documented_tensors_and_metadata(saved):
    adapter, path = saved
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        metadata = handle.metadata()
        names = set(handle.keys())
    assert names == {"pe.radial", "pe.angular", "rope.radial"}
    assert metadata["format"] == "raytun3r-adapter" and metadata["format_version"] == "1"
    assert set(metadata) == {
        "format",
        "format_version",
        "backbone",
        "embed_dim",
        "patch_size",
        "n_r",
        "n_theta",
        "n_r_rope",
        "camera",
        "components",
        "pe_fingerprint",
        "raytun3r_version",
        "training",
    }
    assert json.loads(metadata["camera"])["model"] == "kb4"
    assert set(json.loads(metadata["components"])) == set(COMPONENTS)
    assert json.loads(metadata["training"])["steps"] == 3
    tensors = load_file(str(path))
    assert all(t.dtype == torch.float32 for t in tensors.values())


def test_round_trip_is_exact(saved):
    adapter, path = saved
    loaded = rt.Adapter.load(path)
    assert loaded.same_as(adapter)
    assert loaded.camera == adapter.camera
    assert loaded.training_info == adapter.training_info


def test_save_is_atomic(saved, monkeypatch):
    adapter, path = saved
    before = path.read_bytes()
    import pathlib

    def broken(self, data):  # the disk fills half-way through the temporary file
        with open(self, "wb") as handle:
            handle.write(bytes(data)[: len(data) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(pathlib.Path, "write_bytes", broken)
    with pytest.raises(OSError, match="disk full"):
        randomise_(rt.Adapter.for_model(build_tiny_network(seed=0)), seed=9).save(path)
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def _rewrite(path, tensors=None, **metadata_changes):
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        metadata = dict(handle.metadata())
        current = {k: handle.get_tensor(k) for k in handle.keys()}  # noqa: SIM118
    metadata.update(metadata_changes)
    metadata = {k: v for k, v in metadata.items() if v is not None}
    save_file(current if tensors is None else tensors(current), str(path), metadata=metadata)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(format="something-else"), "metadata 'format' is 'something-else'"),
        (dict(format_version="2"), "format_version '2' is not supported"),
        (dict(backbone=None), "missing metadata \\['backbone'\\]"),
        (dict(n_r="twenty"), "metadata 'n_r' must be a decimal integer, got 'twenty'"),
        (dict(n_r=" 20 "), "metadata 'n_r' must be a decimal integer"),
        (dict(n_r="2_0"), "metadata 'n_r' must be a decimal integer"),
        (dict(n_r="9" * 5000), "metadata 'n_r' must be a decimal integer, got '99999"),
        (dict(n_r="100000"), "metadata 'n_r' must be in \\[2, 1024\\], got 100000"),
        (dict(n_r="21"), "tensor 'pe.radial' has shape \\(20, 64\\), expected \\(21, 64\\)"),
        (dict(components="{not json"), "metadata 'components' is not valid JSON"),
        (dict(components='{"warp": true}'), "'components' must be an object with exactly the keys"),
        (dict(components="7"), "'components' must be an object with exactly the keys"),
        (
            dict(components=json.dumps(dict.fromkeys(COMPONENTS, True) | {"pe_angular": True})),
            "'components' must be an object with exactly the keys",
        ),
        (
            dict(components=json.dumps(dict.fromkeys(COMPONENTS, True) | {"pe_naive_remap": True})),
            "'pe_naive_remap' and 'pe' exclude each other",
        ),
        (dict(components="[[1]]"), "'components' must be an object with exactly the keys"),
        (
            dict(components=json.dumps(dict.fromkeys(COMPONENTS, True) | {"pe": "no"})),
            "'components': 'pe' must be true or false, got 'no'",
        ),
        (
            dict(components='{"pe": true, "pe": false}'),
            "metadata 'components': duplicate key 'pe'",
        ),
        (dict(training='"a string"'), "metadata 'training' must be a JSON object"),
        (dict(training="[1, 2]"), "metadata 'training' must be a JSON object"),
        (dict(training="[" * 5000 + "]" * 5000), "'training' is nested deeper than 32 levels"),
        (dict(training='{"steps": ' + "9" * 5000 + "}"), "'training': integer of 5000 digits"),
        (dict(training='{"loss": NaN}'), "'training': NaN is not JSON"),
        (dict(extra="1"), "unknown metadata \\[\"'extra'\"\\]"),
        (dict(pe_fingerprint="x" * 400), "'pe_fingerprint' must be 16 hex digits"),
        (dict(camera='{"model": "kb4", "width": 84}'), "metadata 'camera' is not a valid camera"),
    ],
)
def test_bad_metadata_is_refused_with_a_clear_message(saved, change, message):
    _adapter, path = saved
    _rewrite(path, **change)
    with pytest.raises(AdapterError, match=message) as error:
        rt.Adapter.load(path)
    assert str(path) in str(error.value)
    assert isinstance(error.value, Raytun3rError)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: {k: v for k, v in t.items() if k != "rope.radial"}, "do not match the expected"),
        (lambda t: t | {"lora.A": torch.zeros(2)}, "do not match the expected"),
        (lambda t: t | {"pe.angular": t["pe.angular"].double()}, "dtype torch.float64"),
        (
            lambda t: (
                t
                | {
                    "pe.radial": t["pe.radial"].masked_fill(
                        torch.eye(20, 64, dtype=torch.bool), float("nan")
                    )
                }
            ),
            "non-finite",
        ),
    ],
)
def test_bad_tensors_are_refused(saved, edit, message):
    _adapter, path = saved
    _rewrite(path, tensors=edit)
    with pytest.raises(AdapterError, match=message):
        rt.Adapter.load(path)


def test_corrupt_and_missing_files(saved, tmp_path):
    _adapter, path = saved
    data = path.read_bytes()
    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(AdapterError, match="not a readable safetensors file"):
        rt.Adapter.load(truncated)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(os.urandom(64))
    with pytest.raises(AdapterError, match="not a readable safetensors file"):
        rt.Adapter.load(garbage)
    with pytest.raises(AdapterError, match="no such adapter file"):
        rt.Adapter.load(tmp_path / "absent.safetensors")


def test_failed_load_leaves_the_model_alone(net, saved):
    _adapter, path = saved
    _rewrite(path, format_version="9")
    with pytest.raises(AdapterError):
        rt.apply(net, fisheye(), str(path))
    assert rt.handle_of(net) is None


def test_describe_file_lists_metadata_camera_and_count(saved):
    adapter, path = saved
    text = describe_file(path)
    assert "backbone:        da3-custom-e64-d6" in text
    assert f"{adapter.num_parameters()['total']:,}" in text
    assert "KannalaBrandt4" in text
