"""Adaptation windows: selection, static skipping, per-pair matches/targets and the disk cache."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from raytun3r_plugin.adaptation.matchers import DISFlowMatcher, Matches
from raytun3r_plugin.adaptation.pose_targets import PoseTarget
from raytun3r_plugin.adaptation.windows import (
    AdaptationSet,
    build_windows,
    prepare_adaptation_set,
    window_pairs,
)
from raytun3r_plugin.cameras import KannalaBrandt4
from raytun3r_plugin.errors import InputError

SIZE = 96
DRIFT = 4  # px per frame after the static start
CAMERA = KannalaBrandt4(SIZE, SIZE, [27.0, 27.0, 47.5, 47.5, 0.0, 0.0, 0.0, 0.0], max_fov_deg=190.0)


class CountingMatcher:
    """DIS at stride 8 that counts its calls (``fast=True``: the cheap ultrafast preset)."""

    name = "counting_dis"

    def __init__(self, stride: int = 8, fast: bool = False) -> None:
        self.inner = (
            DISFlowMatcher(preset="ultrafast", finest_scale=None, stride=stride)
            if fast
            else DISFlowMatcher(stride=stride, appearance_check=False)
        )
        self.calls = 0

    def settings(self) -> dict:
        return {"inner": self.inner.settings()}

    def match(self, image_i, image_j, valid=None) -> Matches:
        self.calls += 1
        return self.inner.match(image_i, image_j, valid)


@pytest.fixture(scope="module")
def segment() -> np.ndarray:
    """12 frames: 0-3 identical (static), then a texture drifting DRIFT px per frame; black
    outside the lens circle."""
    rng = np.random.default_rng(0)
    big = np.zeros((SIZE + 64, SIZE + 64, 3), np.float32)
    for cell, amp in ((4, 0.5), (8, 0.3), (16, 0.2)):
        n = (SIZE + 64) // cell + 2
        noise = rng.random((n, n, 3)).astype(np.float32)
        big += (
            amp
            * cv2.resize(noise, (n * cell, n * cell), interpolation=cv2.INTER_CUBIC)[
                : SIZE + 64, : SIZE + 64
            ]
        )
    mask = CAMERA.valid_mask().numpy()
    frames = []
    for k in range(12):
        s = DRIFT * max(0, k - 3)
        frames.append(np.clip(big[10 + s // 2 : 10 + s // 2 + SIZE, 5 + s : 5 + s + SIZE], 0, 1))
    return (np.stack(frames) * mask[None, :, :, None]).astype(np.float32)


# --------------------------------------------------------------------------- windows


def test_build_windows_spread() -> None:
    w = build_windows(100)
    assert len(w) == 30
    assert w[0] == (0, 1, 2) and w[-1] == (97, 98, 99)
    starts = [x[0] for x in w]
    assert starts == sorted(set(starts))
    assert max(np.diff(starts)) - min(np.diff(starts)) <= 1  # evenly spread
    w2 = build_windows(100, n_windows=4, stride=5, start=10, stop=60)
    assert w2[0] == (10, 15, 20) and w2[-1] == (49, 54, 59)
    assert all(b - a == 5 for x in w2 for a, b in zip(x, x[1:], strict=False))
    # Fewer possible windows than asked for: all of them.
    assert build_windows(5, n_windows=30) == [(0, 1, 2), (1, 2, 3), (2, 3, 4)]
    assert build_windows(10, n_windows=1, window_size=2) == [(0, 1)]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_frames": 2},
        {"n_frames": 10, "stride": 5},
        {"n_frames": 10, "window_size": 1},
        {"n_frames": 10, "n_windows": 0},
        {"n_frames": 10, "start": 8},
        {"n_frames": 10, "stop": 11},
    ],
)
def test_build_windows_errors(kwargs) -> None:
    with pytest.raises(InputError):
        build_windows(**kwargs)


def test_window_pairs_order() -> None:
    assert window_pairs(3) == [(0, 1), (1, 0), (1, 2), (2, 1), (0, 2), (2, 0)]
    assert window_pairs(2) == [(0, 1), (1, 0)]


# --------------------------------------------------------------------------- adaptation set


def test_prepare_skips_static_and_fills_pairs(segment) -> None:
    matcher = CountingMatcher()
    aset = prepare_adaptation_set(segment, CAMERA, matcher, n_windows=10)
    assert isinstance(aset, AdaptationSet)
    candidates = build_windows(12, 10)
    # Windows inside the static frames 0-3 are skipped; the rest move >= 2 px.
    assert aset.static_windows == [(0, 1, 2), (1, 2, 3)]
    assert aset.skipped_static == 2
    assert [w.frames for w in aset.windows] == candidates[2:]
    assert aset.cache_path is None and not aset.from_cache
    for w in aset.windows:
        assert list(w.pairs) == window_pairs(3) and list(w.targets) == window_pairs(3)
        assert w.motion_px >= 2.0
        for (a, b), m in w.pairs.items():
            assert isinstance(m, Matches) and len(m) > 20
            assert isinstance(w.targets[(a, b)], PoseTarget)
            assert w.targets[(a, b)].inlier_mask.shape == (len(m),)
            # Image content moves DRIFT px/frame to the left in u.
            shift = np.median(m.uv_j[:, 0] - m.uv_i[:, 0])
            ga, gb = w.global_pair(a, b)
            expected = -DRIFT * (max(gb, 3) - max(ga, 3))
            assert abs(shift - expected) < 0.5
    # Each global ordered pair is matched once even though windows overlap.
    needed = {(s[a], s[b]) for s in aset.static_windows for a, b in window_pairs(3) if a < b}
    needed |= {w.global_pair(a, b) for w in aset.windows for a, b in window_pairs(3)}
    assert matcher.calls == len(needed)


def test_cache_roundtrip_recomputes_nothing(segment, tmp_path) -> None:
    first = CountingMatcher(fast=True)
    a = prepare_adaptation_set(segment, CAMERA, first, n_windows=2, cache_dir=tmp_path)
    assert first.calls > 0 and not a.from_cache
    assert len(a.windows) == 1 and a.skipped_static == 1  # (9, 10, 11) kept, (0, 1, 2) static
    assert a.cache_path is not None and a.cache_path.suffix == ".npz" and a.cache_path.is_file()
    with np.load(a.cache_path, allow_pickle=False) as data:  # no pickled objects inside
        assert "uv_i" in data.files

    second = CountingMatcher(fast=True)
    b = prepare_adaptation_set(segment, CAMERA, second, n_windows=2, cache_dir=tmp_path)
    assert second.calls == 0 and b.from_cache
    assert b.cache_key == a.cache_key
    assert b.skipped_static == a.skipped_static and b.static_windows == a.static_windows
    assert [w.frames for w in b.windows] == [w.frames for w in a.windows]
    for wa, wb in zip(a.windows, b.windows, strict=True):
        assert wb.motion_px == pytest.approx(wa.motion_px)
        for key in window_pairs(3):
            np.testing.assert_array_equal(wa.pairs[key].uv_i, wb.pairs[key].uv_i)
            np.testing.assert_array_equal(wa.pairs[key].uv_j, wb.pairs[key].uv_j)
            np.testing.assert_array_equal(wa.pairs[key].confidence, wb.pairs[key].confidence)
            ta, tb = wa.targets[key], wb.targets[key]
            np.testing.assert_array_equal(ta.R, tb.R)
            np.testing.assert_array_equal(ta.t, tb.t)
            np.testing.assert_array_equal(ta.inlier_mask, tb.inlier_mask)
            assert (ta.n_inliers, ta.ok, ta.reason) == (tb.n_inliers, tb.ok, tb.reason)

    # Anything that changes the content changes the key.
    keys = {a.cache_key}
    for kwargs in (
        {"threshold_px": 2.0},
        {"n_windows": 1},
        {"min_motion_px": 3.0},
        {"sequence_id": "seq-A"},
    ):
        m = CountingMatcher(fast=True)
        c = prepare_adaptation_set(
            segment, CAMERA, m, **{"n_windows": 2, **kwargs}, cache_dir=tmp_path
        )
        assert not c.from_cache and m.calls > 0
        keys.add(c.cache_key)
    m = CountingMatcher(stride=6, fast=True)
    keys.add(prepare_adaptation_set(segment, CAMERA, m, n_windows=2, cache_dir=tmp_path).cache_key)
    other_camera = KannalaBrandt4(SIZE, SIZE, [27.5, 27.0, 47.5, 47.5, 0.0, 0.0, 0.0, 0.0])
    keys.add(
        prepare_adaptation_set(
            segment, other_camera, CountingMatcher(fast=True), n_windows=2, cache_dir=tmp_path
        ).cache_key
    )
    changed = segment.copy()
    changed[-1, 40, 40] = 0.25
    keys.add(
        prepare_adaptation_set(
            changed, CAMERA, CountingMatcher(fast=True), n_windows=2, cache_dir=tmp_path
        ).cache_key
    )
    assert len(keys) == 8

    # A caller-provided sequence id replaces the image hash (the caller vouches for it).
    m = CountingMatcher(fast=True)
    d = prepare_adaptation_set(
        changed, CAMERA, m, n_windows=2, cache_dir=tmp_path, sequence_id="seq-A"
    )
    assert d.from_cache and m.calls == 0


def test_corrupt_cache_is_recomputed(segment, tmp_path, caplog) -> None:
    a = prepare_adaptation_set(
        segment, CAMERA, CountingMatcher(fast=True), n_windows=2, cache_dir=tmp_path
    )
    a.cache_path.write_bytes(b"not a zip file")
    m = CountingMatcher(fast=True)
    with caplog.at_level(logging.WARNING):
        b = prepare_adaptation_set(segment, CAMERA, m, n_windows=2, cache_dir=tmp_path)
    assert m.calls > 0 and not b.from_cache
    assert "unreadable" in caplog.text
    m2 = CountingMatcher(fast=True)
    c = prepare_adaptation_set(segment, CAMERA, m2, n_windows=2, cache_dir=tmp_path)
    assert c.from_cache and m2.calls == 0


def test_input_errors(segment) -> None:
    small = KannalaBrandt4(64, 64, [18.0, 18.0, 31.5, 31.5, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="rescale"):
        prepare_adaptation_set(segment, small, CountingMatcher(fast=True))
    with pytest.raises(InputError):
        prepare_adaptation_set((segment * 255).astype(np.uint8), CAMERA, CountingMatcher(fast=True))
    with pytest.raises(InputError):
        prepare_adaptation_set(segment[0], CAMERA, CountingMatcher(fast=True))
    with pytest.raises(InputError):
        prepare_adaptation_set(segment * 2.0, CAMERA, CountingMatcher(fast=True))
    with pytest.raises(InputError):
        prepare_adaptation_set(segment, CAMERA, object())
    with pytest.raises(InputError):
        prepare_adaptation_set(segment[:2], CAMERA, CountingMatcher(fast=True))


def test_adaptation_set_on_synthetic_fisheye() -> None:
    """Windows of a rendered ~190 degree KB4 sequence: targets match the true relative poses."""
    import torch

    from raytun3r_plugin import synthetic
    from raytun3r_plugin.adaptation.pose_targets import (
        rotation_error_deg,
        translation_direction_error_deg,
    )

    cam = KannalaBrandt4(
        128, 128, [36.0, 36.0, 63.5, 63.5, 0.01, -0.004, 0.0005, 0.0], max_fov_deg=190.0
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # rendering is much faster without thread contention
    try:
        seq = synthetic.render_sequence("indoor", cam, n_frames=6, seed=0, flow_px=4.0)
    finally:
        torch.set_num_threads(threads)
    aset = prepare_adaptation_set(seq.images, cam, DISFlowMatcher(), n_windows=3)
    assert aset.skipped_static == 0
    assert [w.frames for w in aset.windows] == [(0, 1, 2), (2, 3, 4), (3, 4, 5)]
    for w in aset.windows:
        assert w.motion_px > 2.0
        for (a, b), target in w.targets.items():
            gt = synthetic.relative_pose(seq.cam_from_world, *w.global_pair(a, b))
            assert target.ok, target.reason
            assert rotation_error_deg(target.R, gt[:3, :3]) < 1.0
            assert translation_direction_error_deg(target.t, gt[:3, 3]) < 5.0
