"""An adapter fitted on several segments of one camera at once (``adapt`` with a list of
segments, ``raytun3r adapt --frames A B``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from raytun3r_plugin.patches.da3_networks import build_tiny_network

from raytun3r_plugin import synthetic
from raytun3r_plugin.adaptation.config import AdaptConfig
from raytun3r_plugin.adaptation.problem import prepare_problem, split_segments
from raytun3r_plugin.adaptation.step import objective_value
from raytun3r_plugin.adaptation.train import adapt
from raytun3r_plugin.adapter import Adapter
from raytun3r_plugin.apps.adapter_report import describe_file
from raytun3r_plugin.errors import InputError, Raytun3rError
from tests.helpers import small_kb4


@pytest.fixture(scope="module")
def camera():
    return small_kb4()


@pytest.fixture(scope="module")
def segments(camera):
    return [synthetic.render_sequence("indoor", camera, n_frames=8, seed=seed) for seed in (7, 8)]


def _config(tmp_path, supervised: bool = True, **changes) -> AdaptConfig:
    settings = {
        "steps": 6,
        "input_size": 84,
        "n_windows": 3,
        "checkpoint_every": 0,
        "cache_dir": str(tmp_path),
        "matcher_options": {"border_px": 2},
        "seed": 0,
        **changes,
    }
    return (
        AdaptConfig.supervised(**settings)
        if supervised
        else AdaptConfig.from_recipe("matches", **settings)
    )


def test_split_segments_tells_one_segment_from_several(segments):
    images = segments[0].images
    assert split_segments(images) is None
    assert split_segments(list(images)) is None  # a list of (H, W, 3) frames is one segment
    assert split_segments(torch.from_numpy(images)) is None
    found, depths = split_segments([images, segments[1]])
    assert len(found) == 2 and depths == [None, None]
    found, depths = split_segments((images, images), [segments[0].depth, segments[1].depth])
    assert depths[1] is segments[1].depth
    with pytest.raises(InputError, match="empty list"):
        split_segments([])
    with pytest.raises(InputError, match="mixes whole segments"):
        split_segments([images, images[0]])
    with pytest.raises(InputError, match="list of 2 .* found one array"):
        split_segments([images, images], segments[0].depth)
    with pytest.raises(InputError, match="found a list of 1"):
        split_segments([images, images], [segments[0].depth])
    with pytest.raises(InputError, match="every segment or on none"):
        split_segments([images, images], [segments[0].depth, None])


def test_one_problem_holds_every_segment_with_its_own_frames(camera, segments, tmp_path):
    config = _config(tmp_path)
    depths = [seq.depth for seq in segments]
    single = [prepare_problem(camera, seq.images, config, depth=seq.depth) for seq in segments]
    merged = prepare_problem(camera, [seq.images for seq in segments], config, depth=depths)
    n_first = len(segments[0])
    assert len(merged.windows) == sum(len(p.windows) for p in single)
    for window, _ in merged.windows:  # no window spans two segments
        assert all(f < n_first for f in window.frames) or all(f >= n_first for f in window.frames)
    second = [w for w, _ in merged.windows if w.frames[0] >= n_first]
    assert [tuple(f - n_first for f in w.frames) for w in second] == [
        w.frames for w, _ in single[1].windows
    ]
    for frame, image in single[1].inputs.items():
        assert torch.equal(merged.inputs[frame + n_first], image)
        uv, values = single[1].depth_targets[frame]
        assert torch.equal(merged.depth_targets[frame + n_first][1], values)
    assert merged.supervision["segments"] == 2
    assert merged.supervision["frames"] == sum(p.supervision["frames"] for p in single)
    assert merged.segment["n_frames"] == 2 * n_first and len(merged.segment["segments"]) == 2
    keys = {p.adaptation.cache_key for p in single}
    assert merged.adaptation.cache_key not in keys
    swapped = prepare_problem(
        camera, [seq.images for seq in segments[::-1]], config, depth=depths[::-1]
    )
    assert swapped.adaptation.cache_key != merged.adaptation.cache_key
    # One segment in a list is that segment.
    alone = prepare_problem(camera, [segments[0].images], config, depth=[depths[0]])
    assert alone.adaptation.cache_key == single[0].adaptation.cache_key


def test_a_named_segment_set_caches_each_segment_under_its_own_name(camera, segments, tmp_path):
    config = _config(tmp_path, sequence_id="drive")
    merged = prepare_problem(
        camera, [seq.images for seq in segments], config, depth=[s.depth for s in segments]
    )
    first, second = merged.adaptation.settings["segments"]
    assert first != second  # the same sequence_id would have served segment 0's matches twice
    again = prepare_problem(
        camera, [seq.images for seq in segments], config, depth=[s.depth for s in segments]
    )
    assert again.adaptation.from_cache


def test_a_supervised_fit_on_two_segments_lowers_the_loss_on_both(camera, segments, tmp_path):
    model = build_tiny_network()
    config = _config(tmp_path)
    path = tmp_path / "two.safetensors"
    adapter = adapt(
        model,
        camera,
        [seq.images for seq in segments],
        config,
        depth=[seq.depth for seq in segments],
        out_path=path,
        progress=False,
    )
    info = Adapter.load(path).training_info
    assert info["supervision"]["segments"] == 2
    assert [s["n_frames"] for s in info["segment"]["segments"]] == [8, 8]
    summary = describe_file(path)
    assert "2 segments" in summary and "n_frames 16" in summary
    for seq in segments:
        problem = prepare_problem(camera, seq.images, config, depth=seq.depth)
        before = objective_value(model, Adapter.for_model(model), problem, config)
        after = objective_value(model, adapter, problem, config)
        assert after["depth"] < before["depth"]


def test_a_self_supervised_fit_takes_several_segments(camera, segments, tmp_path):
    model = build_tiny_network()
    config = _config(tmp_path, supervised=False, steps=2, min_parallax_px=0.0)
    adapter = adapt(model, camera, list(segments), config, progress=False)
    info = adapter.training_info
    assert info["supervision"] == {"kind": "self-supervised"}
    assert len(info["segment"]["segments"]) == 2 and info["steps"] == 2


def test_a_bad_segment_is_named_and_nothing_is_written(camera, segments, tmp_path):
    model = build_tiny_network()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    static = np.repeat(segments[1].images[:1], 8, axis=0)
    path = tmp_path / "bad.safetensors"
    with pytest.raises(InputError, match="segment 1 of 2: no usable adaptation window") as caught:
        adapt(
            model,
            camera,
            [segments[0].images, static],
            _config(tmp_path, supervised=False),
            out_path=path,
            progress=False,
        )
    assert isinstance(caught.value, Raytun3rError)
    with pytest.raises(InputError, match="segment 1 of 2: frames are 42x35 px"):
        adapt(
            model,
            camera,
            [segments[0].images, segments[1].images[:, ::2, ::2]],
            _config(tmp_path, supervised=False),
            out_path=path,
            progress=False,
        )
    assert not path.exists()
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())
