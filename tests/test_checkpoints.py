"""Checkpoints as users have them on disk (issue 14): folders, hub snapshots, training files.

DA3 cases use the real ``depth_anything_3`` classes (da3-small at full size builds in well under
a second on CPU; the shipped ``raytun3r-da3-tiny`` for the wrapped files). VGGT / Pi3 cases use
the stubs in tests/stubs through ``tests/backbones.make``, with ``build_network`` swapped for the
tiny stub build exactly as tests/test_vggt_pi3_patch.py does.
"""

from __future__ import annotations

import json
import os
from importlib.util import find_spec

import pytest
import torch
from safetensors.torch import save_file, save_model

import raytun3r_plugin as rt
from raytun3r_plugin.apps.cli import main
from raytun3r_plugin.errors import MissingDependencyError, WeightsError
from raytun3r_plugin.registry import spec_for
from raytun3r_plugin.weights import (
    WEIGHT_FILE_NAMES,
    check_name,
    describe_checkpoint,
    find_weight_file,
    identify_state,
    read_checkpoint,
)

pytest.importorskip("depth_anything_3")
from raytun3r_plugin.patches import da3_networks  # noqa: E402
from raytun3r_plugin.patches import pi3 as pi3_patch  # noqa: E402
from raytun3r_plugin.patches import vggt as vggt_patch  # noqa: E402

from tests.backbones import make  # noqa: E402


class _Wrapper(torch.nn.Module):
    """The ``depth_anything_3.api.DepthAnything3`` layout: the network is ``.model``."""

    def __init__(self, inner: torch.nn.Module) -> None:
        super().__init__()
        self.model = inner


def _da3_config(name: str) -> dict:
    # What DA3's PyTorchModelHubMixin writes: the constructor arguments, model_name first.
    return {"model_name": name, "config": {"net": {"name": "vits"}}}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A da3-small (random weights) saved as the official repository folder is laid out."""
    torch.manual_seed(0)
    net = da3_networks.build_network("da3-small")
    with torch.no_grad():
        for parameter in net.parameters():
            parameter.normal_(0, 0.02)
    folder = tmp_path_factory.mktemp("DA3-SMALL")
    save_model(_Wrapper(net), str(folder / "model.safetensors"))
    (folder / "config.json").write_text(json.dumps(_da3_config("da3-small")))
    return net, folder


def _name(model: torch.nn.Module) -> str:
    spec, root = spec_for(model)
    return spec.describe(root).name


def _same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    reference = a.state_dict()
    return all(torch.equal(reference[k], v) for k, v in b.state_dict().items())


def _fake_da3_state(embed: int, depth: int, rope: bool) -> dict[str, torch.Tensor]:
    """Only the tensors ``identify`` reads (shapes of an official size, values irrelevant)."""
    state = {"model.backbone.pretrained.pos_embed": torch.zeros(1, 1370, embed)}
    for block in range(depth):
        state[f"model.backbone.pretrained.blocks.{block}.attn.qkv.bias"] = torch.zeros(1)
        if rope:
            state[f"model.backbone.pretrained.blocks.{block}.attn.q_norm.weight"] = torch.zeros(1)
    return state


# ---------------------------------------------------------------------------------------------
# Folders, hub snapshots, file preference
# ---------------------------------------------------------------------------------------------


def test_official_folder_loads_and_infers_its_name(small):
    net, folder = small
    loaded = rt.load_backbone(None, folder)
    assert not loaded.training and _same_weights(net, loaded)
    assert _name(loaded) == "da3-small"
    again = rt.load_backbone("da3-small", folder)  # the same folder with its name
    assert _same_weights(net, again)


def test_hub_snapshot_folder_of_symlinks(small, tmp_path):
    _, folder = small
    repo = tmp_path / "models--depth-anything--DA3-SMALL"
    (repo / "blobs").mkdir(parents=True)
    snapshot = repo / "snapshots" / "0123abcd"
    snapshot.mkdir(parents=True)
    for name, blob in (("model.safetensors", "9f8e7d"), ("config.json", "1a2b3c")):
        (repo / "blobs" / blob).write_bytes((folder / name).read_bytes())  # no extension
        os.symlink(os.path.join("..", "..", "blobs", blob), snapshot / name)
    checkpoint = read_checkpoint(snapshot)
    assert checkpoint.path == snapshot / "model.safetensors"
    assert checkpoint.config == _da3_config("da3-small")
    loaded = rt.load_backbone(None, snapshot)
    assert _name(loaded) == "da3-small"
    # The blob itself (extension-less) is recognised as safetensors by its header.
    assert len(read_checkpoint(repo / "blobs" / "9f8e7d").state) == len(checkpoint.state)


def test_folder_prefers_safetensors_then_pt_then_bin(tmp_path):
    assert WEIGHT_FILE_NAMES == ("model.safetensors", "model.pt", "pytorch_model.bin")
    save_file({"w": torch.full((1,), 1.0)}, str(tmp_path / "model.safetensors"))
    torch.save({"w": torch.full((1,), 2.0)}, tmp_path / "model.pt")
    torch.save({"w": torch.full((1,), 3.0)}, tmp_path / "pytorch_model.bin")
    for expected, name in ((1.0, "model.safetensors"), (2.0, "model.pt"), (3.0, None)):
        assert read_checkpoint(tmp_path).state["w"].item() == expected
        if name is not None:
            (tmp_path / name).unlink()
    (tmp_path / "pytorch_model.bin").unlink()
    os.symlink(tmp_path / "gone", tmp_path / "model.safetensors")  # dangling link: skipped
    with pytest.raises(WeightsError, match="folder holds none of the weight files"):
        find_weight_file(tmp_path)


# ---------------------------------------------------------------------------------------------
# Names: config.json, inference, sizes, aliases
# ---------------------------------------------------------------------------------------------


def test_name_disagreeing_with_config_json_is_refused_before_building(small, tmp_path):
    _, folder = small
    other = tmp_path / "DA3-BASE"
    other.mkdir()
    os.symlink(folder / "model.safetensors", other / "model.safetensors")
    (other / "config.json").write_text(json.dumps(_da3_config("da3-base")))
    with pytest.raises(WeightsError) as error:
        rt.load_backbone("da3-small", other)
    message = str(error.value)
    assert "'da3-small'" in message and "'da3-base'" in message and "config.json" in message


def test_release_aliases_agree_with_their_config_and_mono_metric_do_not(small):
    _, folder = small
    assert {"da3-large-1.1", "da3-giant-1.1"} <= set(rt.available_backbones())
    checkpoint = read_checkpoint(folder)
    large = type(checkpoint)(
        path=checkpoint.path,
        state=_fake_da3_state(1024, 24, rope=True),
        config=_da3_config("da3-large"),
    )
    check_name("da3-large-1.1", large, identify_state(large.state))  # same architecture: accepted
    mono = type(checkpoint)(
        path=checkpoint.path,
        state=_fake_da3_state(1024, 24, rope=False),
        config=_da3_config("da3mono-large"),
    )
    with pytest.raises(WeightsError, match="'da3metric-large'.*'da3mono-large'"):
        check_name("da3metric-large", mono, identify_state(mono.state))


def test_none_name_is_inferred_from_shapes_or_refused_when_ambiguous(tmp_path):
    save_file(_fake_da3_state(768, 12, rope=True), str(tmp_path / "base.safetensors"))
    assert describe_checkpoint(tmp_path / "base.safetensors")["name"] == "da3-base"
    save_file(_fake_da3_state(1024, 24, rope=False), str(tmp_path / "mono.safetensors"))
    with pytest.raises(WeightsError, match="da3mono-large.*da3metric-large.*pass the name"):
        rt.load_backbone(None, tmp_path / "mono.safetensors")
    save_file({"x": torch.zeros(2)}, str(tmp_path / "other.safetensors"))
    with pytest.raises(WeightsError, match="no known backbone layout"):
        rt.load_backbone(None, tmp_path / "other.safetensors")


def test_file_of_another_size_names_the_likely_backbone(small, tmp_path, monkeypatch):
    _, folder = small

    def never(name):
        raise AssertionError("built a network for a file of another size")

    monkeypatch.setattr(da3_networks, "build_network", never)  # the refusal comes before any build
    bare = tmp_path / "small.safetensors"  # no config.json next to it: the shapes decide
    os.symlink(folder / "model.safetensors", bare)
    with pytest.raises(WeightsError) as error:
        rt.load_backbone("da3-base", bare)
    with pytest.raises(WeightsError, match="no such weight file"):
        rt.load_backbone("da3-base", tmp_path / "missing.safetensors")
    message = str(error.value)
    assert (
        "'da3-base'" in message and "da3-small" in message and "embed dim 384, 12 blocks" in message
    )


def test_file_of_another_family_is_refused_before_building(small, tmp_path, monkeypatch):
    _, folder = small
    bare = tmp_path / "model.safetensors"
    os.symlink(folder / "model.safetensors", bare)

    def never(*args):
        raise AssertionError("built a network for a file of another family")

    monkeypatch.setattr(vggt_patch, "build_network", never)
    with pytest.raises(WeightsError, match=r"'vggt-1b' \(vggt\).*da3 checkpoint.*da3-small"):
        rt.load_backbone("vggt-1b", bare)


def test_nested_checkpoint_is_recognised_and_built_as_nested(tmp_path, monkeypatch):
    """The nested file names its builder; another size's name is refused before building.

    (Loading a real, tiny nested model end to end: tests/test_nested_da3.py.)
    """
    state = {
        "model.da3." + k.removeprefix("model."): v
        for k, v in _fake_da3_state(1536, 40, rope=True).items()
    }
    state["model.da3_metric.backbone.pretrained.pos_embed"] = torch.zeros(1, 1370, 1024)
    save_file(state, str(tmp_path / "model.safetensors"))
    record = describe_checkpoint(tmp_path)
    assert record["family"] == "da3" and record["name"] == "da3nested-giant-large"
    assert record["load"] == f"raytun3r_plugin.load_backbone('da3nested-giant-large', '{tmp_path}')"

    class Built(Exception):
        pass

    def build(name):
        raise Built(name)

    monkeypatch.setattr(da3_networks, "build_network", build)
    monkeypatch.setitem(da3_networks._NEEDS, "da3nested-giant-large", ())
    with pytest.raises(Built, match="^da3nested-giant-large$"):
        rt.load_backbone(None, tmp_path)
    with pytest.raises(
        WeightsError, match="'da3-large', but the tensors are da3nested-giant-large"
    ):
        rt.load_backbone("da3-large", tmp_path)
    with pytest.raises(
        WeightsError, match="'da3nested-giant-large', but the tensors are da3-large"
    ):
        small = _fake_da3_state(1024, 24, rope=True)
        save_file(small, str(tmp_path / "model.safetensors"))
        rt.load_backbone("da3nested-giant-large", tmp_path)


def test_built_models_record_their_name():
    net = da3_networks.build_network("da3-small")
    assert net.raytun3r_name == "da3-small"
    assert _name(net) == "da3-small"


# ---------------------------------------------------------------------------------------------
# Training checkpoints: wrappers and prefixes, for every family
# ---------------------------------------------------------------------------------------------


def _training_checkpoint(state: dict, wrapper: str, prefix: str) -> dict:
    optimizer = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(2))], lr=1e-4)
    return {
        wrapper: {prefix + key: value for key, value in state.items()},
        "optimizer": optimizer.state_dict(),
        "epoch": 3,
        "prev_epoch": 2,
    }


@pytest.mark.parametrize(
    ("wrapper", "prefix"),
    [("model", "module."), ("model_state_dict", "_orig_mod."), ("state_dict", "module._orig_mod.")],
)
def test_da3_training_checkpoint_is_unwrapped(wrapper, prefix, tmp_path):
    shipped = rt.load_backbone("raytun3r-da3-tiny")
    state = {"model." + key: value for key, value in shipped.state_dict().items()}
    path = tmp_path / "checkpoint.pt"
    torch.save(_training_checkpoint(state, wrapper, prefix), path)
    loaded = rt.load_backbone("raytun3r-da3-tiny", path)
    assert _same_weights(shipped, loaded)
    assert read_checkpoint(path).ignored == ["epoch", "optimizer", "prev_epoch"]


@pytest.mark.parametrize(
    ("name", "wrapper", "prefix"),
    [
        ("vggt-1b", "model", "module."),  # VGGT's trainer under DDP
        ("vggt-1b", "state_dict", "_orig_mod."),
        ("pi3", "model_state_dict", "module._orig_mod."),
        ("pi3x", "model", "_orig_mod."),
    ],
)
def test_vggt_pi3_training_checkpoints_are_unwrapped(name, wrapper, prefix, tmp_path, monkeypatch):
    kind = {"vggt-1b": "vggt", "pi3": "pi3", "pi3x": "pi3x"}[name]
    source = make(kind, seed=1)
    if kind == "vggt":
        monkeypatch.setattr(vggt_patch, "build_network", lambda: make(kind))
    else:
        monkeypatch.setattr(pi3_patch, "build_network", lambda which: make(which))
    path = tmp_path / "checkpoint.pt"
    torch.save(_training_checkpoint(source.state_dict(), wrapper, prefix), path)
    assert describe_checkpoint(path)["family"] == ("vggt" if kind == "vggt" else kind)
    loaded = rt.load_backbone(None, path)  # one size per family: the name follows from the keys
    assert _same_weights(source, loaded)
    assert _name(loaded) == name


def test_unexpected_keys_are_listed_and_known_leftovers_dropped(tmp_path, monkeypatch):
    source = make("vggt", seed=1)
    monkeypatch.setattr(vggt_patch, "build_network", lambda: make("vggt"))
    state = source.state_dict() | {"head.bn.num_batches_tracked": torch.tensor(7)}
    path = tmp_path / "leftover.pt"
    torch.save(state, path)
    assert _same_weights(source, rt.load_backbone("vggt-1b", path))
    torch.save(state | {"ema.decay": torch.zeros(1)}, path)
    with pytest.raises(WeightsError, match=r"unexpected keys \['ema.decay'\]"):
        rt.load_backbone("vggt-1b", path)


def test_vggt_of_another_size_is_a_weights_error(tmp_path, monkeypatch):
    from vggt.models.vggt import VGGT

    other = VGGT(img_size=70, patch_size=14, embed_dim=32, enable_track=False)
    monkeypatch.setattr(vggt_patch, "build_network", lambda: make("vggt"))
    path = tmp_path / "model.safetensors"
    save_file({k: v.contiguous() for k, v in other.state_dict().items()}, str(path))
    with pytest.raises(
        WeightsError,
        match=r"another shape.*aggregator.camera_token \(1, 2, 1, 32\) \(network \(1, 2, 1, 64\)\).*"
        r"the file is a vggt of embed dim 32, 4 aggregator blocks, not the vggt-1b",
    ):
        rt.load_backbone("vggt-1b", path)


def test_a_dict_without_a_state_is_refused(tmp_path):
    path = tmp_path / "meta.pt"
    torch.save({"epoch": 3, "optimizer": {"state": {}}}, path)
    with pytest.raises(WeightsError, match=r"meta.pt: expected a dict of tensors.*'model'"):
        read_checkpoint(path)


# ---------------------------------------------------------------------------------------------
# Dependencies
# ---------------------------------------------------------------------------------------------


@pytest.mark.skipif(find_spec("evo") is not None, reason="evo is installed here")
def test_da3_giant_without_evo_is_a_missing_dependency_before_reading(tmp_path):
    with pytest.raises(
        MissingDependencyError, match=r"'evo'.*pip install evo.*raytun3r\[da3-giant\]"
    ):
        rt.load_backbone("da3-giant-1.1", tmp_path / "not-read.safetensors")
    # The nested model holds a da3-giant: same dependency, also refused before reading.
    with pytest.raises(MissingDependencyError, match=r"'evo'"):
        rt.load_backbone("da3nested-giant-large-1.1", tmp_path / "not-read.safetensors")


# ---------------------------------------------------------------------------------------------
# raytun3r weights
# ---------------------------------------------------------------------------------------------


def test_cli_weights_describes_a_folder(small, capsys):
    _, folder = small
    assert main(["weights", str(folder)]) == 0
    text = capsys.readouterr().out
    assert "family    da3" in text
    assert "name      da3-small  (config.json: da3-small)" in text
    assert "PE table  1x1370x384" in text and "float32" in text
    assert f"load      raytun3r_plugin.load_backbone('da3-small', '{folder}')" in text
    assert main(["weights", str(folder), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["tensors"] == len(read_checkpoint(folder).state)
    assert record["pe_shape"] == [1, 1370, 384] and record["dtypes"] == {
        "float32": record["tensors"]
    }
    assert record["candidates"] == ["da3-small"]


def test_cli_weights_reports_ignored_training_entries(tmp_path, capsys):
    shipped = rt.load_backbone("raytun3r-da3-tiny")
    path = tmp_path / "checkpoint.pt"
    torch.save(_training_checkpoint(shipped.state_dict(), "model", "module."), path)
    assert main(["weights", str(path)]) == 0
    text = capsys.readouterr().out
    assert "ignored   epoch, optimizer, prev_epoch" in text
    assert "family    da3" in text and "blocks, RoPE" in text
    assert "load      - (pass the name" in text  # a custom size: the name is not in the file


def test_cli_weights_on_unknown_and_missing_files(tmp_path, capsys):
    save_file({"x": torch.zeros(2, dtype=torch.float16)}, str(tmp_path / "x.safetensors"))
    assert main(["weights", str(tmp_path / "x.safetensors")]) == 0
    text = capsys.readouterr().out
    assert "family    unknown" in text and "float16 (1)" in text and "pass the name" in text
    assert main(["weights", str(tmp_path / "missing")]) == 2
    assert "no such weight file" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# Full-size official builds
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("name", ["da3metric-large", "da3mono-large", "da3-large-1.1"])
def test_official_large_builds_report_their_own_name(name):
    net = da3_networks.build_network(name)
    assert _name(net) == name


@pytest.mark.slow
@pytest.mark.skipif(find_spec("evo") is not None, reason="evo is installed here")
def test_da3_giant_import_failure_inside_the_build_is_a_missing_dependency(monkeypatch):
    monkeypatch.setattr(da3_networks, "_NEEDS", {})  # skip the pre-check: upstream's import fails
    with pytest.raises(MissingDependencyError, match=r"'evo'.*pip install evo"):
        da3_networks.build_network("da3-giant")
