"""The rig fit runs on the loop ``adapt`` runs on (``adaptation/loop.py``): the collapse guard,
checkpoints and resuming, Ctrl-C, and the supervised mode (docs/rigs.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import raytun3r_plugin as rt
from raytun3r_plugin.adaptation import AdaptConfig, rig
from raytun3r_plugin.adaptation.rig import adapt_rig, rig_artifact_paths
from raytun3r_plugin.errors import InputError
from raytun3r_plugin.synthetic.generate import render_rig
from tests.helpers import assert_same_snapshot, fisheye, snapshot


@pytest.fixture(scope="module")
def stereo():
    cameras = {"left": fisheye(56, 56, 190.0), "right": fisheye(56, 56, 165.0, k1=0.03)}
    return render_rig("indoor", cameras, n_frames=6, seed=7, flow_px=5.0)


def _network():
    from raytun3r_plugin.patches.da3_networks import build_tiny_network

    return build_tiny_network(seed=0).eval()


def _config(**changes):
    settings = dict(
        steps=4, input_size=56, n_windows=2, checkpoint_every=0, min_parallax_px=0.0, lr=3e-2
    )
    settings.update(changes)
    return AdaptConfig.from_recipe("matches", **settings)


def _tables(fitted):
    return {
        f"{n}.{k}": v.detach().clone() for n, a in fitted.items() for k, v in a.state_dict().items()
    }


def test_the_rig_guard_restores_every_camera_when_the_joint_depth_collapses(stereo, monkeypatch):
    # A correlation no changed depth can reach: the first check after a step trips.
    monkeypatch.setattr(rig, "GUARD_MIN_CORRELATION", 1.5)
    fitted = adapt_rig(_network(), stereo, _config(guard_every=2), progress=False)
    for adapter in fitted.values():
        info = adapter.training_info
        assert info["guard"]["tripped"]["step"] == 2
        assert info["guard"]["tripped"]["restored_step"] == 0
        assert info["verdict"]["status"] == "collapsed" and info["steps"] == 2
        # Restored to the tables of step 0: the zero adapter.
        assert all(float(p.detach().abs().sum()) == 0.0 for p in adapter.parameters())
    # With the shipped thresholds the same fit is healthy and keeps its tables.
    monkeypatch.undo()
    healthy = adapt_rig(_network(), stereo, _config(guard_every=2), progress=False)
    for adapter in healthy.values():
        assert adapter.training_info["guard"]["tripped"] is None
        assert adapter.training_info["steps"] == 4
        assert sum(float(p.detach().abs().sum()) for p in adapter.parameters()) > 0


def test_an_interrupted_rig_fit_resumes_to_the_uninterrupted_tables(stereo, tmp_path, monkeypatch):
    config = _config(checkpoint_every=2, guard=False)
    straight = adapt_rig(_network(), stereo, config, out_dir=tmp_path / "straight", progress=False)

    original = rig.rig_step

    def interrupted_at_3(model, fitted, problems, names, optimizer, config, step, *args):
        if step == 3:
            raise KeyboardInterrupt
        return original(model, fitted, problems, names, optimizer, config, step, *args)

    monkeypatch.setattr(rig, "rig_step", interrupted_at_3)
    model = _network()
    before = snapshot(model)
    stopped = adapt_rig(model, stereo, config, out_dir=tmp_path / "run", progress=False)
    assert rt.handle_of(model) is None
    assert_same_snapshot(model, before)
    info = stopped["left"].training_info
    assert info["interrupted"] is True and info["steps"] == 3
    paths = rig_artifact_paths(tmp_path / "run", ["left", "right"])
    assert paths["checkpoint"].is_file() and paths["adapter:left"].is_file()

    monkeypatch.setattr(rig, "rig_step", original)
    resumed = adapt_rig(model, stereo, config, out_dir=tmp_path / "run", progress=False)
    info = resumed["right"].training_info
    assert info["resumed_from"] == 3 and info["steps"] == 4 and info["interrupted"] is False
    log = [json.loads(line) for line in paths["log"].read_text().splitlines()]
    assert [r["step"] for r in log] == [0, 1, 2, 3]
    expected, got = _tables(straight), _tables(resumed)
    assert expected.keys() == got.keys()
    for key in expected:
        torch.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-7)
    # Another run's checkpoint is refused, not silently continued.
    with pytest.raises(rt.Raytun3rError, match="another run"):
        adapt_rig(
            model,
            stereo,
            _config(checkpoint_every=2, guard=False, lr=1e-3),
            out_dir=tmp_path / "run",
            progress=False,
        )


def test_the_supervised_rig_fit_scores_each_camera_against_its_depth(stereo):
    depth = {name: seq.depth for name, seq in stereo.sequences.items()}
    config = AdaptConfig.from_recipe(
        "supervised", steps=3, input_size=56, n_windows=2, checkpoint_every=0, guard=False
    )
    fitted = adapt_rig(_network(), stereo, config, progress=False, depth=depth)
    for name, adapter in fitted.items():
        info = adapter.training_info
        assert info["supervision"]["kind"] == "depth"
        assert info["method"] == "raytun3r supervised rig adaptation"
        assert "depth" in info["final_losses"] and "reproj" not in info["final_losses"]
        assert sum(float(p.detach().abs().sum()) for p in adapter.parameters()) > 0, name


def test_a_supervised_rig_request_missing_a_camera_is_refused_before_anything(stereo):
    model = _network()
    before = snapshot(model)
    left = stereo.sequences["left"].depth
    with pytest.raises(InputError, match="right"):
        adapt_rig(model, stereo, progress=False, depth={"left": left})
    with pytest.raises(InputError, match="cross-camera"):
        adapt_rig(
            model,
            stereo,
            progress=False,
            depth={"left": left, "right": np.asarray(left)},
            cross_camera=True,
        )
    assert rt.handle_of(model) is None
    assert_same_snapshot(model, before)
