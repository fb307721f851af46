"""load_backbone: local weights only, official key layout, strict but alias-tolerant."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from safetensors.torch import save_file, save_model

import raytun3r_plugin as rt
from raytun3r_plugin.errors import MissingDependencyError, WeightsError
from raytun3r_plugin.weights import alias_keys

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches.da3_networks import build_network  # noqa: E402


@pytest.fixture(scope="module")
def official(tmp_path_factory):
    """A randomly initialised da3-small written the way the released checkpoint is laid out."""
    torch.manual_seed(0)
    net = build_network("da3-small")
    with torch.no_grad():
        for parameter in net.parameters():
            parameter.normal_(0, 0.02)
    folder = tmp_path_factory.mktemp("weights")

    class Wrapper(torch.nn.Module):  # the DepthAnything3 wrapper stores the network as .model
        def __init__(self, inner):
            super().__init__()
            self.model = inner

    path = folder / "model.safetensors"
    save_model(Wrapper(net), str(path))  # drops shared-tensor aliases exactly like the release
    return net, path


def test_round_trip_in_official_layout(official):
    net, path = official
    loaded = rt.load_backbone("da3-small", path)
    assert not loaded.training
    reference = net.state_dict()
    assert all(torch.equal(reference[k], v) for k, v in loaded.state_dict().items())


def test_aliases_are_exactly_the_shared_layernorm(official):
    net, _ = official
    assert sorted(alias_keys(net)) == sorted(
        f"head.scratch.output_conv2_aux.{i}.2.{p}" for i in (1, 2, 3) for p in ("weight", "bias")
    )


def test_pt_file_through_weights_only(official, tmp_path):
    net, _ = official
    path = tmp_path / "model.pt"
    torch.save({"model." + k: v for k, v in net.state_dict().items()}, path)
    loaded = rt.load_backbone("da3-small", path)
    assert torch.equal(loaded.backbone.pretrained.pos_embed, net.backbone.pretrained.pos_embed)


def test_pickled_objects_are_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"model.x": torch.zeros(1), "hook": object()}, path)
    with pytest.raises(WeightsError, match="weights_only=True"):
        rt.load_backbone("da3-small", path)


def test_missing_and_unexpected_keys_are_errors(official, tmp_path):
    net, _ = official
    state = {
        k: v
        for k, v in net.state_dict().items()
        if not k.startswith("head.scratch.output_conv2_aux.1")
    }
    state["model.extra.weight"] = torch.zeros(3)
    path = tmp_path / "bad.safetensors"
    save_file({k: v.clone().contiguous() for k, v in state.items()}, str(path))
    with pytest.raises(WeightsError) as error:
        rt.load_backbone("da3-small", path)
    message = str(error.value)
    assert "missing keys" in message and "head.scratch.output_conv2_aux.1.0" in message
    assert "unexpected keys ['extra.weight']" in message


def test_no_path_and_unknown_names():
    with pytest.raises(WeightsError, match="needs a local weight file"):
        rt.load_backbone("da3-small")
    with pytest.raises(WeightsError, match="unknown backbone 'da3-huge'"):
        rt.load_backbone("da3-huge", "x.safetensors")
    assert {"da3-small", "da3-base", "da3-large"} <= set(rt.available_backbones())
    with pytest.raises(WeightsError, match="no such weight file"):
        rt.load_backbone("da3-small", "/nonexistent/model.safetensors")


def test_loading_never_imports_huggingface_hub(official):
    _, path = official
    code = (
        "import sys, raytun3r_plugin as rt; rt.load_backbone('da3-small', sys.argv[1]);"
        "print('huggingface_hub' in sys.modules)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip().splitlines()[-1] == "False"


def test_missing_upstream_gives_install_hint(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_da3(name, *args, **kwargs):
        if name.startswith("depth_anything_3"):
            raise ImportError("No module named 'depth_anything_3'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_da3)
    with pytest.raises(MissingDependencyError, match="pip install --no-deps depth-anything-3"):
        build_network("da3-small")
