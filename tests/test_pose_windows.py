"""``AdaptConfig.pose_windows``: the pose term only where the matches carry no depth.

With ``"unreprojected"`` a window whose matches enter the reprojection term gets no pose term,
and a window the parallax gate keeps for the teacher alone keeps it. So where every window
reprojects the fit is the targets fit (no pose term at all), and where none does it is the
default ``"all"`` fit, table for table. Off by default and out of the identity when off.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
from raytun3r_plugin.patches.da3_networks import build_tiny_network

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.errors import InputError
from tests.helpers import small_fit_config, small_kb4


@pytest.fixture(scope="module")
def room():
    camera = small_kb4()
    return camera, synthetic.render_sequence("indoor", camera, n_frames=6, seed=7)


def _config(tmp_path, **changes) -> AdaptConfig:
    """The default recipe on the small room, its teacher on whatever the lens."""
    return small_fit_config(tmp_path, "default", teacher_max_coverage=1.0, lr=3e-2, **changes)


def _fit(room, config, out=None):
    camera, seq = room
    return adapt(build_tiny_network(), camera, seq.images, config, progress=False, out_path=out)


def _records(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _same_tables(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters(), strict=True))


def test_pose_windows_is_validated_and_out_of_the_identity_when_all():
    assert "pose_windows" not in AdaptConfig().to_dict()
    on = AdaptConfig(pose_windows="unreprojected")
    assert on.to_dict()["pose_windows"] == "unreprojected"
    assert on.identity() != AdaptConfig().identity()
    for changes in (
        {"pose_windows": "some"},
        {"pose_windows": "unreprojected", "pose_source": "model"},
        {"pose_windows": "unreprojected", "pose_source": "targets"},
    ):
        with pytest.raises(InputError, match="AdaptConfig.pose_windows"):
            AdaptConfig(**changes)


def test_where_every_window_reprojects_the_pose_term_is_left_out(room, tmp_path):
    """No parallax gate: every window's matches reproject, so the pose term scores none of them
    and the fit is the targets fit (reprojection through the targets and the teacher)."""
    base = _config(tmp_path, min_parallax_px=0.0)
    fitted = _fit(room, dataclasses.replace(base, pose_windows="unreprojected"), tmp_path / "w")
    records = _records(tmp_path / "w.log.jsonl")
    assert len(records) == 4
    assert all(r["n_pose"] == 0 and r["pose"] == 0.0 and r["n_matches"] > 0 for r in records)
    assert _same_tables(fitted, _fit(room, dataclasses.replace(base, pose_source="targets")))
    everywhere = _fit(room, base, tmp_path / "a")
    assert all(r["n_pose"] > 0 for r in _records(tmp_path / "a.log.jsonl"))
    assert not _same_tables(fitted, everywhere)
    assert fitted.training_info["config"]["pose_windows"] == "unreprojected"


def test_where_no_window_reprojects_the_fit_is_the_default_one(room, tmp_path):
    """A gate no window passes, with the teacher on: every window keeps the pose term, so the
    fit is the one with ``pose_windows="all"``, table for table."""
    base = _config(tmp_path, min_parallax_px=1e6)
    windowed = _fit(room, dataclasses.replace(base, pose_windows="unreprojected"), tmp_path / "w")
    assert windowed.training_info["parallax_gate"]["windows_reprojected"] == 0
    assert all(r["n_pose"] > 0 and r["reproj"] == 0.0 for r in _records(tmp_path / "w.log.jsonl"))
    assert _same_tables(windowed, _fit(room, base))


def test_the_pose_gate_drops_the_setting_with_the_term(room, tmp_path):
    """A pose gate that switches the fit to the targets takes ``pose_windows`` back to
    ``"all"`` with it, instead of refusing its own switch."""
    config = _config(tmp_path, min_parallax_px=0.0, pose_windows="unreprojected", pose_gate=1e9)
    fitted = _fit(room, config)
    assert fitted.training_info["pose_gate"]["pose_term"] is False
