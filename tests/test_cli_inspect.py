"""``raytun3r inspect``: a readable summary by default, the raw record with ``--json``."""

from __future__ import annotations

import json

import pytest

from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.cli import main
from tests.helpers import fisheye, randomise_

TRAINING = {
    "method": "raytun3r online adaptation",
    "steps": 120,
    "requested_steps": 200,
    "resumed_from": 40,
    "interrupted": True,
    "final_losses": {"loss": 0.1234567, "photometric": 0.0812, "pose": 0.0421},
    "final_losses_over_steps": 8,
    "segment": {
        "name": "corridor",
        "start": 10,
        "frames": 60,
        "mask": None,
        "windows": [[0, 1, 2], [3, 4, 5]],
        "skipped_static": 1,
    },
    "input": {"width": 504, "height": 406, "crop": None},
    "adaptation_set": "0123456789abcdef" * 4,
    "config": {"steps": 200, "lr": 0.01, "window": 3},
    "wall_time_s": 38.25,
}


@pytest.fixture
def adapter_file(tmp_path):
    adapter = randomise_(
        Adapter("da3-small", embed_dim=64, patch_size=14, camera=fisheye(), training=TRAINING)
    )
    return adapter.save(tmp_path / "adapter.safetensors")


def test_inspect_prints_a_readable_summary(adapter_file, capsys):
    assert main(["inspect", str(adapter_file)]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert len(lines) >= 10 and not any("{" in line for line in lines)  # no one-line JSON dump
    assert "da3-small" in text and "KannalaBrandt4" in text
    assert "120 of 200 steps" in text and "resumed at step 40" in text and "interrupted" in text
    assert "loss 0.123" in text and "photometric 0.0812" in text
    assert "corridor" in text and "2 windows" in text and "504x406" in text
    assert "38.2 s" in text or "38.3 s" in text
    assert "--json" in text  # says where the full record is


def test_inspect_json_prints_the_raw_record(adapter_file, capsys):
    assert main(["inspect", "--json", str(adapter_file)]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["training"] == TRAINING
    assert record["backbone"] == "da3-small" and record["camera"]["model"] == "kb4"
    assert record["parameters"]["total"] == Adapter.load(adapter_file).num_parameters()["total"]


def test_inspect_of_an_unfitted_adapter(tmp_path, capsys):
    path = Adapter("da3-small", embed_dim=64, camera=fisheye()).save(tmp_path / "zero.safetensors")
    assert main(["inspect", str(path)]) == 0
    text = capsys.readouterr().out
    assert "not fitted" in text and "identity adapter" in text
